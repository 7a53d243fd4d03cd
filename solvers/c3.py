"""The C3 / C3+ controller's public API (the algorithm itself is :mod:`c3bench.solvers.admm`).

The consensus ADMM (QP step, projection, dual update, residuals, rho schedules, stopping,
output, warm start) is defined once in :mod:`c3bench.solvers.admm` (docs/admm.md); this module
re-exports its entry points under their historical names and holds what surrounds the
controller: the LCS rollout with Lemke's ``lam``, the sample weighting of the robust
controller, and the capture of ADMM iterates for the suites.

**Sample weights** (:func:`lcp_prediction_weights`, seed 000 section 3.3): each sample
predicts every past observation ``(x, u, x_next)`` with its LCS, ``lam`` from the LCP
``0 <= lam perp F lam + E x + H u + c >= 0`` solved by Lemke's method, and
``x_hat = A x + B u + D lam + d``; its error is ``e_j = sum_t ||x_next_t - x_hat_t||^2`` and
its weight ``p_j = exp(-(e_j - min e) / temperature) / sum``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from c3bench.problems.capture import Capture, CaptureContext, CapturedIterate
from c3bench.problems.families import weight_vector
from c3bench.problems.lcs import LCS, LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import BLOCKS
from c3bench.solvers.admm.controller import C3Controller, solve_c3, solve_robust
from c3bench.solvers.admm.loop import (
    cold_iterates,
    dual_update,
    normalise_weights,
    rescale_dual,
    shift_warm_start,
)
from c3bench.solvers.admm.options import (
    OUTPUTS,
    RHO_SCHEDULES,
    STOPPING_RULES,
    VARIANTS,
    WEIGHT_FLOOR,
    C3Options,
)
from c3bench.solvers.admm.projection import make_step_projection
from c3bench.solvers.admm.schedules import schedule_for
from c3bench.solvers.admm.solution import C3Iterate, C3Solution, C3Trace
from c3bench.solvers.admm.stacked import (
    full_layout,
    mpcc_vector,
    project_step_c3,
    qp_layout,
    to_full_steps,
)
from c3bench.solvers.lcp import lemke

__all__ = ["OUTPUTS", "RHO_SCHEDULES", "STOPPING_RULES", "VARIANTS", "WEIGHT_FLOOR",
           "C3Controller", "C3Iterate", "C3Options", "C3Solution", "C3Trace", "cold_start",
           "controller_capture", "dual_update", "full_layout", "iterate_to_capture",
           "lcp_prediction_errors", "lcp_prediction_weights", "lcp_step", "next_rho",
           "normalise_weights", "project_step_c3", "project_step_c3plus", "qp_layout",
           "rescale_dual", "rho_multiplier", "rollout", "rollout_vector", "shift_warm_start",
           "solve_c3", "solve_robust", "to_full_steps",
           "weight_vector"]


def rho_multiplier(options: C3Options, consensus: float, consensus_prev: float | None,
                   dual: float) -> float:
    """The schedule's factor after an iteration (:mod:`c3bench.solvers.admm.schedules`)."""
    previous = math.inf if consensus_prev is None else consensus_prev
    return float(schedule_for(options).multiplier(consensus, previous, dual))


def next_rho(options: C3Options, rho: Mapping[str, float], consensus: float,
             consensus_prev: float | None, dual: float) -> dict[str, float]:
    """``rho_{i+1}``: the scheduled blocks times :func:`rho_multiplier`."""
    return schedule_for(options).next(rho, consensus, consensus_prev, dual)


def cold_start(lcs: LCS, x0: np.ndarray, horizon: int, variant: str
               ) -> tuple[np.ndarray, np.ndarray]:
    """``delta_k = (x0, 0, 0, 0)``, ``w = 0`` (T x step size of the QP layout)."""
    delta, w = cold_iterates(qp_layout(lcs, horizon, variant), x0, 1)
    return delta[0], w[0]


def project_step_c3plus(v: np.ndarray, layout: HorizonLayout, rho: Mapping[str, float]
                        ) -> np.ndarray:
    """C3+'s projection of steps ``v`` (..., step size) in ``G(rho)``: ``x, u`` copied, pairs in
    closed form (:func:`c3bench.solvers.admm.projection.make_step_projection`)."""
    project = make_step_projection(np, layout.nx, layout.nlam, layout.nu)
    inf = np.full(layout.nx + layout.nu, np.inf)
    out: np.ndarray = project(np.asarray(v, dtype=float), math.sqrt(rho["lam"]),
                              math.sqrt(rho["eta"]), -inf, inf, None, False)
    return out




# --- LCS rollout and sample scoring -----------------------------------------------------------
def lcp_step(lcs: LCS, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """One LCS step with ``lam`` from Lemke: ``(x_next, lam)``, or ``None`` when Lemke fails."""
    solution = lemke(lcs.F, lcs.lcp_offset(x, u))
    if not solution.found or solution.z is None:
        return None
    lam = solution.z
    return lcs.next_state(x, u, lam), lam


def rollout(lcs: LCS, x0: np.ndarray, inputs: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Simulate the LCS from ``x0`` under ``inputs`` (T x nu) with Lemke's ``lam``.

    Returns ``(xs (T+1 x nx), lams (T x nlam), etas (T x nlam))``, a point that satisfies the
    dynamics and complementarity of the mpcc exactly (to Lemke's precision), or ``None`` when
    an LCP has no solution found.
    """
    xs = [np.asarray(x0, dtype=float)]
    lams, etas = [], []
    for u in np.asarray(inputs, dtype=float):
        step = lcp_step(lcs, xs[-1], u)
        if step is None:
            return None
        x_next, lam = step
        lams.append(lam)
        etas.append(lcs.gap(xs[-1], u, lam))
        xs.append(x_next)
    return np.array(xs), np.array(lams), np.array(etas)


def rollout_vector(lcs: LCS, mpc: MPC, x0: np.ndarray, inputs: np.ndarray
                   ) -> np.ndarray | None:
    """:func:`rollout` of the inputs clipped to the force limit, as an mpcc vector."""
    layout = full_layout(lcs, mpc.horizon)
    us = np.clip(np.asarray(inputs, dtype=float), -mpc.force_limit, mpc.force_limit)
    simulated = rollout(lcs, x0, us)
    if simulated is None:
        return None
    xs, lams, etas = simulated
    steps = np.zeros((mpc.horizon, layout.step_size))
    steps[:, layout.index(0, "x")] = xs[:-1]
    steps[:, layout.index(0, "lam")] = lams
    steps[:, layout.index(0, "u")] = us
    steps[:, layout.index(0, "eta")] = etas
    return mpcc_vector(steps, xs[-1])


Observation = tuple[np.ndarray, np.ndarray, np.ndarray]


def lcp_prediction_errors(lcs_samples: Sequence[LCS], observations: Sequence[Observation]
                          ) -> np.ndarray:
    """``e_j = sum_t ||x_next_t - x_hat_j(x_t, u_t)||_2^2`` per sample (``inf`` when Lemke
    fails on one of its LCPs); ``x_hat`` from :func:`lcp_step`."""
    errors = np.zeros(len(lcs_samples))
    for j, lcs in enumerate(lcs_samples):
        for x, u, x_next in observations:
            step = lcp_step(lcs, np.asarray(x, dtype=float), np.asarray(u, dtype=float))
            if step is None:
                errors[j] = math.inf
                break
            errors[j] += float(np.sum((np.asarray(x_next, dtype=float) - step[0]) ** 2))
    return errors


def lcp_prediction_weights(lcs_samples: Sequence[LCS] | LCSBatch,
                           observations: Sequence[Observation],
                           temperature: float | None = None,
                           compiled: bool = True) -> np.ndarray:
    """Sample weights from one-step LCP prediction errors (seed 000, section 3.3).

    ``p_j = exp(-(e_j - min_i e_i) / temperature) / sum`` with ``e_j`` from
    :func:`lcp_prediction_errors`. ``temperature=None`` takes the median finite error (floored
    at 1e-12): a sample with a median error gets ``e^-1`` of the best sample's weight, whatever
    the units. A sample whose prediction failed gets weight 0; with no observations, or when
    every prediction failed, the weights are uniform (nothing to judge by).

    ``compiled`` (default) computes the errors of all samples and observations in one numba
    call (:func:`c3bench.solvers.lcp_batch.lcp_prediction_errors_batch`, equal to
    :func:`lcp_prediction_errors` to 1e-10: tests/test_lcp_batch.py); ``False`` runs the scalar
    reference above. An :class:`LCSBatch` is used as is (no per-sample ``LCS`` objects).
    """
    from c3bench.solvers import lcp_batch  # numba loads on first use, not with this module

    S = lcs_samples.n_samples if isinstance(lcs_samples, LCSBatch) else len(lcs_samples)
    if S == 0:
        raise ValueError("need at least one sample")
    if len(observations) == 0:
        return np.full(S, 1.0 / S)
    if compiled:
        weights: np.ndarray = lcp_batch.lcp_prediction_weights_batch(lcs_samples, observations,
                                                                     temperature)
        return weights
    samples = lcs_samples.samples() if isinstance(lcs_samples, LCSBatch) else lcs_samples
    reference: np.ndarray = lcp_batch.prediction_weights(
        lcp_prediction_errors(samples, observations), temperature)
    return reference


# --- capture for the suites -------------------------------------------------------------------
def iterate_to_capture(iterate: C3Iterate, lcs: LCS, layout: HorizonLayout, source: str,
                       sample: int = 0) -> CapturedIterate:
    """One iteration in the suites' C3+ layout.

    A C3 run's ``eta`` columns are filled from the LCS: ``delta_eta = E x + F lam + H u + c``
    of ``delta``, ``w_eta = E w_x + F w_lam + H w_u`` (no ``c``: ``w`` is a difference, so
    ``(delta - w)`` keeps ``eta`` equal to its gap) and ``v_eta`` the gap of ``v = z + w``.
    """
    delta = to_full_steps(iterate.delta[sample], lcs, layout)
    w = to_full_steps(iterate.w[sample], lcs, layout, homogeneous=True)
    v = to_full_steps(iterate.projection_v[sample], lcs, layout)
    return CapturedIterate(iteration=iterate.iteration,
                           rho={k: float(iterate.rho[k]) for k in BLOCKS},
                           delta=delta, w=w, projection_v=v, source=source)


def controller_capture(options: C3Options | None = None) -> Capture:
    """A capture function for :func:`problems.suites.generate_suite` that runs the controller.

    At each sampled state it runs :func:`solve_c3` from a cold start on the context's LCS and
    MPC, with a fixed iteration count covering every iteration the suite asks for (at least
    ``options.admm_iterations``), and yields every completed iteration as a
    :class:`c3bench.problems.capture.CapturedIterate` (C3+ layout, :func:`iterate_to_capture`) with
    ``source = "controller:<variant>/<qp_backend>"``. Deterministic when the backends are.
    Iterations after a QP failure do not exist and are not yielded.
    """
    base = options or C3Options()

    def capture(context: CaptureContext) -> list[CapturedIterate]:
        spec = context.spec
        needed = 1 + max((*spec.admm_iterations, *spec.projection_iterations), default=0)
        run = replace(base, admm_iterations=max(base.admm_iterations, needed),
                      stopping="fixed", keep_iterates=True)
        solution = solve_c3(context.lcs, context.mpc, context.x0, run,
                            fallback_input=context.u_prev)
        return [iterate_to_capture(it, context.lcs, solution.layout, run.source)
                for it in solution.iterates]

    return capture

