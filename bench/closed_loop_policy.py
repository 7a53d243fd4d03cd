"""The controllers of the closed loop: :class:`ControllerSpec` (which controller, and how) and
:func:`make_policy` (the ``policy(x, t) -> (u, info)`` that :func:`bench.closed_loop.simulate`
calls every control step).

The reference controllers (``c3``, ``c3plus``, ``c3plus-robust``, :mod:`solvers.c3`) solve their
QP steps (and C3 its projections) with registry backends; :func:`step_backends` runs those
under a per-solve time limit (``ControllerSpec.qp_time_limit``) so that a hanging backend is
killed and the step counted as failed (:func:`step_failures`) instead of hanging the run. The
fast controllers (:mod:`solvers.fast`) solve their QP steps themselves.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

import numpy as np

from c3bench.problems.config import Config
from c3bench.problems.errors import InputError
from c3bench.problems.lcs import ContactModel
from c3bench.problems.names import LcsKernel, Variant
from c3bench.problems.scene import Scene, build_scene

if TYPE_CHECKING:
    from c3bench.solvers.base import Backend

CONTROLLERS: tuple[str, ...] = ("c3", "c3plus", "c3plus-robust", "c3plus-fast",
                                 "c3plus-fast-robust")
ROBUST_CONTROLLERS: tuple[str, ...] = ("c3plus-robust", "c3plus-fast-robust")
FAST_CONTROLLERS: tuple[str, ...] = ("c3plus-fast", "c3plus-fast-robust")


class ContactModelOption(StrEnum):
    """``--contact-model``: the contact model of the controller's LCS
    (:func:`c3bench.problems.lcs.assemble_lcs`). Anitescu's relaxation (default) makes a
    sliding contact separate at ``mu |v_t|`` (docs/lcs.md); Stewart-Trinkle keeps it closed
    at the price of a slack per contact (``nlam`` grows from ``contacts x directions`` to
    ``contacts x (directions + 2)``)."""

    ANITESCU = "anitescu"
    STEWART_TRINKLE = "stewart-trinkle"

    @property
    def lcs_name(self) -> ContactModel:
        """The name :func:`c3bench.problems.linearize.linearize` takes."""
        return "anitescu" if self is ContactModelOption.ANITESCU else "stewart_trinkle"

    @classmethod
    def parse(cls, value: str) -> ContactModelOption:
        """``value`` (``stewart_trinkle`` accepted for ``stewart-trinkle``) as an option;
        :class:`InputError` naming ``--contact-model`` otherwise."""
        text = value.replace("_", "-") if isinstance(value, str) else value
        try:
            return cls(text)
        except ValueError:
            raise InputError(f"--contact-model must be one of "
                             f"{', '.join(m.value for m in cls)}, got {value!r}") from None


Policy = Callable[[np.ndarray, float], tuple[np.ndarray, dict[str, Any]]]
"""``policy(x, t) -> (u, info)``; ``info`` may carry ``lcs_time``, ``solve_time``, ``ok``,
``nan_count``, ``qp_failures`` (int), ``qp_failure`` and ``fallback_reason`` (str) and scalar
diagnostics."""


@dataclass(frozen=True)
class ControllerSpec:
    """Which controller drives the plant, and how.

    Attributes
    ----------
    controller
        ``c3`` (MIQP projection), ``c3plus`` (closed-form projection), ``c3plus-robust``
        (``samples`` models with ``l ~ U[l_low, l_high]`` sharing their inputs, one stacked
        QP), or the fast path ``c3plus-fast`` / ``c3plus-fast-robust`` (batched Riccati QP
        steps and batched LCS build, :mod:`solvers.fast`; ``qp_backend`` is ignored).
    qp_backend, projection
        Registry names of the QP-step solver and of C3's MIQP projection.
    rho_schedule
        ``geometric`` (the reference study's), ``adaptive`` or ``residual_balancing``.
    admm_iterations
        ADMM iterations per control step (seed: 10).
    model_l
        Cube side of the single model (seed: the shrunk 0.29).
    samples, l_low, l_high
        Robust variant: number of sampled models and the range of their sides.
    weighting
        Robust variant: weight samples by their one-step LCP prediction error on the
        observations so far (seed section 3.3).
    seed
        Seed of the sampled sides.
    feedback, feedback_kp, feedback_kd
        Low-level feedback between control steps (the reference study's "low-level PD controller"):
        at every plant step ``u = u_0 + kp (p_ref - p) + kd (v_ref - v)`` on the ball, where
        ``p_ref`` moves linearly from the measured ball position to the plan's ``x_1`` over
        ``dt`` and ``v_ref`` is the plan's ``x_1`` ball velocity (weighted over samples).
        Without it ``u_0`` is held for ``dt`` (zero-order hold). The reference study's optimised
        gain ``K`` regularised toward a PD law is not implemented.
    contact_model
        The controller's LCS contact model, a :class:`ContactModelOption` value
        (``anitescu`` or ``stewart-trinkle``; the plant is MuJoCo either way).
    qp_time_limit
        Wall-clock seconds allowed to each solve of the QP backend (and of C3's projection
        backend) in :func:`bench.closed_loop.run_closed_loop`: the backend then runs in a
        persistent child process (:class:`~c3bench.solvers.isolation.IsolatedBackend`) that is
        killed when a solve overruns, and the step falls back (counted in ``qp_failures``), so
        a hanging backend cannot hang the loop. ``None`` calls the backend in this process,
        unguarded. The fast controllers have no backend and ignore it.

        **Cost.** Every QP solve then makes a round trip to the child (the dense QP pickled
        there, the result back) and the measured step times include it, as step 0 includes
        starting the child (and, once per process, the forkserver that preloads the solvers).
        Measured on the 2-core VM under a load average of 2.5-7 from parallel test runs: the
        single-model C3+ QP (``n = 178``, 437 kB pickled) costs 1-2.3 ms more per solve than
        in-process (1.3-1.8 ms), so a 10-iteration C3+ control step took 15-17 ms longer
        (25 -> 40 ms with Clarabel, 28 -> 45 ms with OSQP at load 2.6: +55-60 %); the
        16-sample robust QP (``n = 2638``, 97 MB pickled) costs about 0.4 s more CPU and
        0.8 s more wall time per solve than its 0.12 s, some 3x the step time. C3's MIQP
        projections (seconds per step) see no measurable difference. The limit stays on by
        default (a hung backend is worse than a slow step); ``None`` measures step times
        without the round trips.
    """

    controller: str = "c3plus"
    qp_backend: str = "clarabel"
    projection: str = "scip"
    rho_schedule: str = "geometric"
    admm_iterations: int = 10
    model_l: float = 0.29
    samples: int = 16
    l_low: float = 0.27
    l_high: float = 0.33
    weighting: bool = True
    seed: int = 0
    feedback: bool = False
    feedback_kp: float = 100.0
    feedback_kd: float = 20.0
    qp_time_limit: float | None = 10.0
    contact_model: str = ContactModelOption.ANITESCU.value
    warm_dual: str = "zero"

    def __post_init__(self) -> None:
        """Check every field (:class:`InputError` naming the option and the allowed range)."""
        from c3bench.solvers.c3 import RHO_SCHEDULES

        object.__setattr__(self, "contact_model",
                           ContactModelOption.parse(self.contact_model).value)
        if self.controller not in CONTROLLERS:
            raise InputError(f"--controller must be one of {', '.join(CONTROLLERS)}, got "
                             f"{self.controller!r}")
        from c3bench.solvers.admm.options import DUAL_WARM_STARTS

        if self.warm_dual not in DUAL_WARM_STARTS:
            raise InputError(f"warm_dual must be one of {', '.join(DUAL_WARM_STARTS)}, got "
                             f"{self.warm_dual!r}")
        if self.rho_schedule not in RHO_SCHEDULES:
            raise InputError(f"--rho-schedule must be one of {', '.join(RHO_SCHEDULES)}, "
                             f"got {self.rho_schedule!r}")
        for option, value in (("--samples", self.samples),
                              ("--iterations", self.admm_iterations)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) \
                    or value < 1:
                raise InputError(f"{option} must be an integer >= 1, got {value!r}")
        positive = [("--model-l", self.model_l), ("l_low", self.l_low),
                    ("l_high", self.l_high)]
        if self.qp_time_limit is not None:
            positive.append(("--qp-time-limit", self.qp_time_limit))
        for option, number in positive:
            if not (isinstance(number, int | float) and math.isfinite(number) and number > 0):
                raise InputError(f"{option} must be a finite number > 0, got {number!r}")
        if self.l_low > self.l_high:
            raise InputError(f"need l_low <= l_high, got {self.l_low}, {self.l_high}")
        for option, gain in (("feedback_kp", self.feedback_kp),
                             ("feedback_kd", self.feedback_kd)):
            if not (isinstance(gain, int | float) and math.isfinite(gain) and gain >= 0):
                raise InputError(f"{option} must be a finite number >= 0, got {gain!r}")

    def sample_sides(self) -> np.ndarray:
        """The robust variant's model sides (seeded, sorted)."""
        rng = np.random.default_rng(self.seed)
        return np.sort(rng.uniform(self.l_low, self.l_high, self.samples))

    @property
    def robust(self) -> bool:
        return self.controller in ROBUST_CONTROLLERS

    def label(self) -> str:
        extra = f"-n{self.samples}" if self.robust else f"-l{self.model_l:g}"
        backend = "compiled" if self.controller in FAST_CONTROLLERS else self.qp_backend
        feedback = "-pd" if self.feedback else ""
        contact = "" if self.contact_model == ContactModelOption.ANITESCU else "-st"
        dual = "" if self.warm_dual == "zero" else f"-w{self.warm_dual}"
        return (f"{self.controller}-{backend}-{self.rho_schedule}{extra}{feedback}{contact}"
                f"{dual}")

    @property
    def lcs_contact_model(self) -> ContactModel:
        """The contact model's name for the LCS builders."""
        return ContactModelOption(self.contact_model).lcs_name


@contextlib.contextmanager
def step_backends(spec: ControllerSpec) -> Iterator[dict[str, Backend]]:
    """The controller's QP (and C3's projection) backends under ``spec.qp_time_limit``.

    Yields ``{registry name: IsolatedBackend(backend, qp_time_limit)}`` for the backends the
    controller calls (nothing for the fast controllers or without a limit) and closes them
    (their child processes end) on exit. Each wrapper keeps one child process for the whole
    run and starts a new one only after a kill.
    """
    if spec.controller in FAST_CONTROLLERS or spec.qp_time_limit is None:
        yield {}
        return
    from c3bench.solvers import registry
    from c3bench.solvers.isolation import IsolatedBackend

    names = [spec.qp_backend] + ([spec.projection] if spec.controller == "c3" else [])
    with contextlib.ExitStack() as stack:
        wrapped: dict[str, Backend] = {}
        for name in dict.fromkeys(names):
            wrapped[name] = stack.enter_context(
                IsolatedBackend(registry.get(name), spec.qp_time_limit))
        yield wrapped


def step_failures(solution: Any) -> tuple[int, str]:
    """``(failed sub-solves, first reason)`` of a control step's solution.

    The reference controller's trace marks every failed QP step or projection
    (:class:`solvers.c3.C3Trace`: ``failed``, ``message``); the fast path has no backend and
    no such trace: ``(0, "")``.
    """
    trace = getattr(solution, "trace", None)
    if trace is None or not hasattr(trace, "failed"):
        return 0, ""
    reasons = [str(message) for failed, message in zip(trace.failed, trace.message,
                                                       strict=True) if failed]
    return len(reasons), reasons[0] if reasons else ""


def make_policy(spec: ControllerSpec, config: Config,
                backends: Mapping[str, Backend] | None = None) -> Policy:
    """A policy that linearises the controller's model(s) at the measured state and runs C3.

    The LCS is built at ``(x, u_prev)`` every control step (``lcs_time``); the controller warm
    starts from its previous step. The robust variants weight their samples by the one-step
    LCP prediction error on the last five observed transitions ``(x_t, u_t, x_{t+1})`` (one
    compiled call, :mod:`solvers.lcp_batch`). The reference controller (the reference kernel
    of :mod:`solvers.admm`, any registry QP backend) and the fast path (the compiled kernel
    :class:`solvers.admm.compiled_solver.CompiledC3Plus`, batched LCS build) run the same
    ADMM loop and differ only in how the models are built and the kernel.

    ``backends`` replaces registry backends by name (:func:`step_backends`, which
    :func:`bench.closed_loop.run_closed_loop` uses); without it the registry's backends run
    in this process.
    """
    from c3bench.problems.scene import build_mpc
    from c3bench.solvers.c3 import lcp_prediction_weights

    sides = spec.sample_sides() if spec.robust else np.array([spec.model_l])
    scene = build_scene(l=float(sides[0]), config=config)
    mpc = build_mpc(scene, config.mpc)
    dt = config.mpc.dt
    if spec.controller in FAST_CONTROLLERS:
        from c3bench.problems.linearize_batch import BatchLinearizer
        from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
        from c3bench.solvers.fast import FastC3PlusController, fast_options
        from c3bench.solvers.lcp_batch import warm_up

        linearizer = BatchLinearizer(sides, config, contact_model=spec.lcs_contact_model,
                                     kernel=LcsKernel.COMPILED)
        fast = FastC3PlusController(CompiledC3Plus(mpc, fast_options(
            rho_schedule=spec.rho_schedule, admm_iterations=spec.admm_iterations,
            warm_dual=spec.warm_dual)))
        warm_up()  # the compiled Lemke of the weighting: loaded once, outside the steps
        linearizer.warm_up()  # the compiled LCS build, likewise

        def models_at(x: np.ndarray, u: np.ndarray) -> Any:
            return linearizer.linearize(x, u, dt)

        def samples_of(models: Any) -> list[Any]:
            return models.samples()

        def solve(models: Any, weights: Sequence[float] | None, x: np.ndarray) -> Any:
            return fast.step(models, x, weights)
    else:
        from c3bench.problems.linearize import linearize
        from c3bench.solvers.c3 import C3Controller, C3Options

        scenes = [scene] + [build_scene(l=float(side), config=config) for side in sides[1:]]
        reference = C3Controller(C3Options(
            variant=Variant.C3 if spec.controller == "c3" else Variant.C3PLUS,
            qp_backend=spec.qp_backend, projection_backend=spec.projection,
            rho_schedule=spec.rho_schedule, admm_iterations=spec.admm_iterations,
            warm_dual=spec.warm_dual,
            keep_iterates=False, backends=dict(backends or {})))

        def models_at(x: np.ndarray, u: np.ndarray) -> Any:
            return [linearize(model, x, u, dt, spec.lcs_contact_model) for model in scenes]

        def samples_of(models: Any) -> list[Any]:
            return models

        def solve(models: Any, weights: Sequence[float] | None, x: np.ndarray) -> Any:
            if spec.robust:
                return reference.step_robust(models, weights, mpc, x)
            return reference.step(models[0], mpc, x)

    history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    previous: dict[str, np.ndarray] = {}

    def policy(x: np.ndarray, t: float) -> tuple[np.ndarray, dict[str, Any]]:
        u_prev = previous.get("u", np.zeros(scene.nu))
        if "x" in previous:
            history.append((previous["x"], u_prev, x.copy()))
        start = time.perf_counter()
        models = models_at(x, u_prev)
        lcs_time = time.perf_counter() - start
        start = time.perf_counter()
        weights: Sequence[float] | None = None
        if spec.robust and spec.weighting:
            # an LCSBatch (fast path) or a list of LCS: the compiled weighting takes either
            weights = lcp_prediction_weights(models, history[-5:]).tolist()
        weight_time = time.perf_counter() - start
        solution = solve(models, weights, x)
        solve_time = time.perf_counter() - start
        u = np.asarray(solution.u, dtype=float)
        previous["x"], previous["u"] = x.copy(), u.copy()
        raw = solution.u_raw
        failures, first_failure = step_failures(solution)
        info: dict[str, Any] = {
            "lcs_time": lcs_time, "solve_time": solve_time, "weight_time": weight_time,
            "ok": solution.ok, "iterations": solution.iterations,
            "nan_count": int(not solution.ok and raw is not None
                             and not np.all(np.isfinite(raw))),
            "qp_failures": failures, "qp_failure": first_failure,
            "fallback_reason": "" if solution.ok else str(solution.status)}
        trace = getattr(solution, "trace", None)
        residuals = trace.consensus_residual if trace is not None \
            else solution.consensus_residual
        if residuals:
            info["consensus_residual"] = float(residuals[-1])
        if trace is not None and trace.complementarity_delta:
            info["complementarity_delta"] = float(trace.complementarity_delta[-1])
        info.update(plan_arrays(samples_of(models), solution, x))
        if spec.feedback and solution.ok:
            plan = planned_ball_state(solution.delta, solution.weights, scene.nq,
                                      scene.ball_position_indices, scene.nq - scene.nv)
            info["control_law"] = pd_tracking_law(spec, scene, x, plan, dt)
        return u, info

    return policy


def plan_arrays(samples: Sequence[Any], solution: Any, x: np.ndarray) -> dict[str, Any]:
    """The step's plan for the metrics (:mod:`bench.closed_loop_metrics`): ``commanded`` (the
    unclipped ``u_0``), and, when the step succeeded, ``plan_next`` (the plan's ``x_1``),
    ``lcs_next`` (the LCS rollout of the plan's ``u_0`` from ``x``) and ``plan_input``."""
    from c3bench.bench.closed_loop_metrics import plan_prediction

    raw = solution.u_raw
    out: dict[str, Any] = {}
    if raw is not None:
        commanded = np.asarray(raw, dtype=float)
        out["commanded"] = commanded.reshape(-1, commanded.shape[-1])[0].copy()
    if not solution.ok or not np.all(np.isfinite(solution.delta)):
        return out
    plan, rollout, first = plan_prediction(samples, solution.delta, solution.weights, x)
    out.update({"plan_next": plan, "lcs_next": rollout, "plan_input": first})
    return out


def planned_ball_state(delta: np.ndarray, weights: np.ndarray | None, nq: int,
                       ball: np.ndarray, nv_offset: int) -> tuple[np.ndarray, np.ndarray]:
    """Ball position and velocity of the plan's ``x_1`` (``delta`` is (S, T, step), ``x``
    first in each step), averaged over samples with ``weights``."""
    x1 = np.asarray(delta)[:, 1 if delta.shape[1] > 1 else 0, :]
    p = np.full(x1.shape[0], 1.0 / x1.shape[0]) if weights is None else \
        np.asarray(weights, dtype=float) / np.sum(weights)
    mean = p @ x1
    return mean[ball], mean[nq + ball - nv_offset]


def pd_tracking_law(spec: ControllerSpec, scene: Scene, x: np.ndarray,
                    reference: tuple[np.ndarray, np.ndarray], dt: float
                    ) -> Callable[[np.ndarray, float, np.ndarray], np.ndarray]:
    """``law(x, s, u0) = u0 + kp (p_ref(s) - p) + kd (v_ref - v)`` on the ball (see
    :class:`ControllerSpec` ``feedback``)."""
    ball = scene.ball_position_indices
    ball_v = scene.nq + ball - (scene.nq - scene.nv)
    start = x[ball].copy()
    end, velocity = reference

    def law(state: np.ndarray, s: float, u0: np.ndarray) -> np.ndarray:
        target = start + (end - start) * min(1.0, s / dt)
        return u0 + spec.feedback_kp * (target - state[ball]) \
            + spec.feedback_kd * (velocity - state[ball_v])

    return law
