"""The closed-loop suites' configurations: which controllers a suite runs, the claims it
tests, and the suites themselves (:data:`CLOSED_LOOP_SUITES`).

Run by :func:`bench.closed_loop_suite.run_cases`.

Suites (:data:`CLOSED_LOOP_SUITES`, :class:`ClosedLoopSuite`): *configurations* (a
controller, a group, a display name) x N randomized trials (:mod:`bench.trials`: ball start
+-3 cm, cube mass +-20 %, friction +-25 %, plant side U[0.28, 0.32] m; seed
:data:`SUITE_SEED`, so trial ``i`` is the same episode in both suites and whatever N, and a
run resumes or extends the stored one):

* ``quick``, 20 trials each: stacked C3+ (shrunk model ``l = 0.29``, geometric rho, 10 ADMM
  iterations) with Clarabel and OSQP and with the true-size model (``l = 0.30``, Clarabel);
  the seed's method (fast robust C3+, 16 samples, LCP weighting, feedback); the fast robust
  variants without feedback, weighted and uniform; the reference study's ablation
  (:func:`reference_ablation`, fast path); the success-vs-``l`` curve (:data:`L_CURVE`: the
  ablation's ``no-samples`` with its side varied). A controller asked for twice runs once
  (:attr:`Configuration.also`): 15 configurations, 300 episodes;
* ``full``, 100 trials each: the same with the QP backends of :data:`FULL_BACKENDS` and C3
  with its MIQP projection (Gurobi, SCIP): 23 configurations.

``--trials N`` (``c3bench closed-loop-suite``) overrides the count. Measured on the 2-core VM
(load average 1-2, this suite the only heavy job): 2 trials of ``quick`` (30 episodes) took
35 s with two workers, the stacked C3+ episodes 3-5 s each (50-100 ms per step), the fast
robust ones 0.6-1.2 s, the fast single-model ones 0.2-0.4 s; under a load average of 4-5
from other jobs, the next 30 episodes took 61 s. The 300 episodes of ``quick`` take about 6
minutes on a quiet machine, 10 on a busy one; ``full`` takes hours (C3's MIQP projection
takes seconds per step).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from c3bench.bench.cli_options import MAX_TRIALS
from c3bench.bench.closed_loop import ControllerSpec
from c3bench.bench.trials import trial_case
from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError

if TYPE_CHECKING:
    from c3bench.bench.closed_loop_suite import Case


def _c3plus(backend: str, **changes: Any) -> ControllerSpec:
    return ControllerSpec(controller="c3plus", qp_backend=backend, **changes)


QUICK_BACKENDS: tuple[str, ...] = ("clarabel", "osqp")
"""QP backends of the stacked C3+ in the quick suite."""
FULL_BACKENDS: tuple[str, ...] = (*QUICK_BACKENDS, "equilibrated_kkt",
                                  "equilibrated_kkt_noridge", "proxqp_sparse", "daqp",
                                  "kkt_ldl", "casadi_hpipm")
"""QP backends of the stacked C3+ in the full suite."""
L_CURVE: tuple[float, ...] = (0.27, 0.28, 0.29, 0.295, 0.30, 0.31)
"""Model cube sides (m) of the success-vs-``l`` curve: fast C3+ with one model and feedback
(the ablation's ``no-samples`` with its side varied; 0.29 and 0.30 are the ablation's
``no-samples`` and ``no-shrunk-model``)."""
QUICK_TRIALS = 20
FULL_TRIALS = 100
SUITE_SEED = 0
"""Seed of the trial draws of both suites (trial ``i`` is the same episode in both)."""



def check_trials(count: Any) -> int:
    """``count`` trials per configuration: an integer in ``[1, MAX_TRIALS]``
    (:data:`c3bench.bench.cli_options.MAX_TRIALS`), else :class:`InputError` naming
    ``--trials``."""
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_TRIALS:
        raise InputError(f"--trials must be an integer in [1, {MAX_TRIALS}], got {count!r}")
    return count

class SuiteGroup(StrEnum):
    """What a configuration of a closed-loop suite stands for (one colour per group in the
    report's figures)."""

    BACKENDS = "backends"
    SEED_METHOD = "seed method"
    ROBUST = "robust"
    ABLATION = "ablation"
    L_CURVE = "l-curve"
    C3 = "c3"


def reference_ablation() -> list[tuple[str, ControllerSpec]]:
    """The reference study's ablation (its bar plot): the full method, one part removed each.

    Full: robust C3+ (16 samples ``l ~ U[0.27, 0.33]``, LCP-error weighting) with low-level
    feedback, on the fast path. Removed in turn: feedback, the samples (one model, the shrunk
    ``l = 0.29``), the samples and the shrunk model (one model of the true ``l = 0.30``), the
    weighting; and the two other rho schedules.
    """
    full = ControllerSpec(controller="c3plus-fast-robust", feedback=True)
    return [
        ("full", full),
        ("no-feedback", replace(full, feedback=False)),
        ("no-samples", replace(full, controller="c3plus-fast", model_l=0.29)),
        ("no-shrunk-model", replace(full, controller="c3plus-fast", model_l=0.30)),
        ("no-weighting", replace(full, weighting=False)),
        ("rho-adaptive", replace(full, rho_schedule="adaptive")),
        ("rho-residual-balancing", replace(full, rho_schedule="residual_balancing")),
    ]


@dataclass(frozen=True)
class Configuration:
    """One controller of a closed-loop suite, run for every trial of the suite.

    Attributes
    ----------
    name
        File-safe unique name: the prefix of its cases and the ``config`` column.
    group
        A :class:`SuiteGroup` value.
    spec
        The controller (the robust ones get a fresh model seed per trial:
        :func:`bench.trials.trial_case`).
    title
        Display name in the report.
    also
        Other roles the same controller plays in the suite (a controller that two parts of
        the suite ask for runs once, e.g. the ablation's ``no-samples`` is the ``l = 0.29``
        point of the success-vs-``l`` curve).
    """

    name: str
    group: str
    spec: ControllerSpec
    title: str
    also: tuple[str, ...] = ()


def _with_role(configurations: list[Configuration], name: str, group: str,
               spec: ControllerSpec, title: str) -> None:
    """Append a configuration, or add ``title`` as another role of an equal controller."""
    for index, known in enumerate(configurations):
        if known.spec == spec:
            configurations[index] = replace(known, also=(*known.also, title))
            return
    configurations.append(Configuration(name, group, spec, title))


def suite_configurations(backends: Sequence[str], with_c3: bool) -> tuple[Configuration, ...]:
    """The configurations of a suite: stacked C3+ per QP backend (shrunk model ``l = 0.29``)
    and with the true-size model; the seed's method; the robust variants; the ablation; the
    success-vs-``l`` curve (:data:`L_CURVE`); with ``with_c3``, C3 with each MIQP projection.
    Controllers asked for twice run once (:attr:`Configuration.also`)."""
    out: list[Configuration] = []
    add = out.append
    for backend in backends:
        add(Configuration(f"c3plus-{backend}-l0.29", SuiteGroup.BACKENDS, _c3plus(backend),
                          f"C3+ {backend}, l 0.29"))
    add(Configuration("c3plus-clarabel-l0.3", SuiteGroup.BACKENDS,
                      _c3plus("clarabel", model_l=0.30), "C3+ clarabel, true l 0.30"))
    ablation = dict(reference_ablation())
    add(Configuration("seed-method", SuiteGroup.SEED_METHOD, ablation["full"],
                      "seed method (fast robust, weighted, feedback)", ("ablation full",)))
    robust = replace(ablation["full"], feedback=False)
    _with_role(out, "robust-weighted", SuiteGroup.ROBUST, robust, "fast robust, weighted")
    _with_role(out, "robust-uniform", SuiteGroup.ROBUST, replace(robust, weighting=False),
               "fast robust, uniform")
    for label, spec in reference_ablation()[1:]:
        _with_role(out, f"ablation-{label}", SuiteGroup.ABLATION, spec, f"ablation {label}")
    for side in L_CURVE:  # the ablation's no-samples with the model side varied
        _with_role(out, f"fast-l{side:g}", SuiteGroup.L_CURVE,
                   replace(ablation["full"], controller="c3plus-fast", model_l=side),
                   f"l-curve {side:g}")
    if with_c3:
        for projection in ("gurobi", "scip"):
            spec = ControllerSpec(controller="c3", qp_backend="clarabel", projection=projection)
            add(Configuration(f"c3-clarabel-{projection}", SuiteGroup.C3, spec,
                              f"C3 clarabel + {projection}"))
    return tuple(out)


def l_curve_points(configurations: Sequence[Configuration]) -> tuple[tuple[float, str], ...]:
    """``(model side, configuration name)`` of the success-vs-``l`` curve: for each side of
    :data:`L_CURVE`, the configuration that runs the ablation's ``no-samples`` controller with
    that side (skipped when the suite has none)."""
    no_samples = dict(reference_ablation())["no-samples"]
    points = []
    for side in L_CURVE:
        spec = replace(no_samples, model_l=side)
        names = [c.name for c in configurations if c.spec == spec]
        if names:
            points.append((side, names[0]))
    return tuple(points)


class SeedClaim(StrEnum):
    """The seed's design choices that the randomized trials test."""

    SHRUNK_MODEL = "shrunk model"
    WEIGHTING = "LCP weighting"
    FEEDBACK = "low-level feedback"


@dataclass(frozen=True)
class Comparison:
    """One test of a :class:`SeedClaim`: configuration ``with_choice`` (the seed's choice)
    against ``without`` (the choice removed), everything else equal; ``setting`` says what
    the two share."""

    claim: SeedClaim
    with_choice: str
    without: str
    setting: str


COMPARISONS: tuple[Comparison, ...] = (
    Comparison(SeedClaim.SHRUNK_MODEL, "c3plus-clarabel-l0.29", "c3plus-clarabel-l0.3",
               "stacked C3+ (clarabel), one model, no feedback: l 0.29 vs 0.30"),
    Comparison(SeedClaim.SHRUNK_MODEL, "ablation-no-samples", "ablation-no-shrunk-model",
               "fast C3+, one model, feedback: l 0.29 vs 0.30"),
    Comparison(SeedClaim.WEIGHTING, "seed-method", "ablation-no-weighting",
               "fast robust C3+, 16 samples, feedback: weighted vs uniform"),
    Comparison(SeedClaim.WEIGHTING, "robust-weighted", "robust-uniform",
               "fast robust C3+, 16 samples, no feedback: weighted vs uniform"),
    Comparison(SeedClaim.FEEDBACK, "seed-method", "robust-weighted",
               "fast robust C3+, 16 samples, weighted: feedback vs none"),
)
"""The pairs the report compares (Newcombe's interval for the difference of the success
rates: :func:`bench.trials.newcombe_interval`)."""


@dataclass(frozen=True)
class ClosedLoopSuite:
    """Configurations x randomized trials (:mod:`bench.trials`).

    Attributes
    ----------
    name
        ``quick`` or ``full``: the directory ``ROOT/closed_loop/<name>/``.
    configurations
        The controllers.
    trials
        Episodes per configuration (``--trials`` overrides it).
    seed
        Seed of the draws: trial ``i`` is the same episode for every configuration and
        whatever the number of trials, so a run with more trials reuses the stored ones.
    duration, hold_time
        Seconds per episode and seconds the angle must stay in the band at the end.
    comparisons
        The claims the report tests (:data:`COMPARISONS`; one naming a configuration the
        suite lacks is skipped).
    """

    name: str
    configurations: tuple[Configuration, ...]
    trials: int
    seed: int = SUITE_SEED
    duration: float = 3.0
    hold_time: float = 1.0
    comparisons: tuple[Comparison, ...] = COMPARISONS

    @property
    def l_curve(self) -> tuple[tuple[float, str], ...]:
        """:func:`l_curve_points` of the configurations."""
        return l_curve_points(self.configurations)

    def cases(self, trials: int | None = None) -> list[Case]:
        """Every episode: ``trials`` (default :attr:`trials`) per configuration, named
        ``<configuration>-<trial, 4 digits>``, trials outermost (an interrupted run has
        the first trials of every configuration rather than all trials of the first)."""
        count = check_trials(self.trials if trials is None else trials)
        base = load_config()
        cases = []
        for index in range(count):
            for configuration in self.configurations:
                case = trial_case(configuration.spec, index, self.seed, self.duration,
                                  self.hold_time, base=base)
                cases.append(replace(case, name=f"{configuration.name}-{index:04d}",
                                     group=str(configuration.group),
                                     configuration=configuration.name, trial=index))
        return cases


CLOSED_LOOP_SUITES: dict[str, ClosedLoopSuite] = {
    "quick": ClosedLoopSuite("quick", suite_configurations(QUICK_BACKENDS, with_c3=False),
                             QUICK_TRIALS),
    "full": ClosedLoopSuite("full", suite_configurations(FULL_BACKENDS, with_c3=True),
                            FULL_TRIALS),
}


__all__ = [
    "CLOSED_LOOP_SUITES", "COMPARISONS", "FULL_BACKENDS", "FULL_TRIALS", "L_CURVE",
    "QUICK_BACKENDS", "QUICK_TRIALS", "SUITE_SEED", "ClosedLoopSuite", "Comparison",
    "Configuration", "SeedClaim", "SuiteGroup", "l_curve_points", "reference_ablation",
    "suite_configurations",
]
