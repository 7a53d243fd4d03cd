"""Randomized closed-loop trials: one controller, N episodes with perturbed physics.

Each trial ``i`` of seed ``S`` draws, from ``numpy.random.default_rng([S, i])`` (so a trial
is the same whatever N, and trials differ from one another):

* the ball's start, ``x`` and ``z`` each moved by ``U[-3, 3] cm``;
* the plant cube's mass, ``x U[0.8, 1.2]`` (+-20 %);
* the table and ball friction coefficients, each ``x U[0.75, 1.25]`` (+-25 %);
* the plant cube's side, ``U[0.28, 0.32]`` m;
* for the robust controllers, the seed of their sampled model sides.

The controller keeps the nominal constants (its model does not know the draw). The trials run
as closed-loop cases (:func:`bench.closed_loop_suite.run_cases`: local process pool or Dask,
locked, resumable, one stored cell per episode) and are summarised by the success rate with
its Wilson score 95 % interval (E. B. Wilson, "Probable inference, the law of succession, and
statistical inference", J. Am. Stat. Assoc. 22 (1927) 209-212), the gentle-success rate,
the medians of the physical metrics (:mod:`bench.closed_loop_metrics`) and the counts of the
labels (:mod:`bench.closed_loop_labels`) (:func:`trial_summary`). Two configurations' success
rates are compared by Newcombe's hybrid score interval for the difference of two independent
proportions (:func:`newcombe_interval`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from c3bench.bench.closed_loop_policy import ControllerSpec
from c3bench.problems.config import Config, load_config

if TYPE_CHECKING:  # the suite module imports this one (its report uses the statistics)
    from c3bench.bench.closed_loop_suite import Case

Z_95 = 1.959963984540054
"""The standard normal's 97.5 % quantile: a two-sided 95 % interval."""


@dataclass(frozen=True)
class TrialRanges:
    """How far each trial perturbs the plant (module docstring).

    Attributes
    ----------
    ball_offset
        Half-width of the uniform shift of the ball's start, in x and in z (m).
    mass
        Relative half-width of the cube mass factor.
    friction
        Relative half-width of each friction coefficient's factor.
    side
        Range of the plant cube's side (m).
    """

    ball_offset: float = 0.03
    mass: float = 0.20
    friction: float = 0.25
    side: tuple[float, float] = (0.28, 0.32)


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson's (1927) score interval for a binomial proportion.

    ``(p + z^2 / 2n -+ z sqrt(p (1 - p) / n + z^2 / 4n^2)) / (1 + z^2 / n)`` with
    ``p = successes / trials``; ``(0, 1)`` when there are no trials.
    """
    if trials <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be in [0, {trials}], got {successes}")
    p = successes / trials
    scale = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / scale
    half = z / scale * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials))
    return max(0.0, centre - half), min(1.0, centre + half)


def newcombe_interval(successes_a: int, trials_a: int, successes_b: int, trials_b: int,
                      z: float = Z_95) -> tuple[float, float]:
    """Newcombe's hybrid score interval for the difference ``p_a - p_b`` of two independent
    proportions (method 10 of R. G. Newcombe, "Interval estimation for the difference between
    independent proportions: comparison of eleven methods", Stat. Med. 17 (1998) 873-890).

    With ``(l_a, u_a)``, ``(l_b, u_b)`` the Wilson intervals (:func:`wilson_interval`) of
    ``p_a = successes_a / trials_a`` and ``p_b``:

    ``L = (p_a - p_b) - sqrt((p_a - l_a)^2 + (u_b - p_b)^2)``,
    ``U = (p_a - p_b) + sqrt((u_a - p_a)^2 + (p_b - l_b)^2)``.

    The difference is significant at the 95 % level when the interval excludes 0; this is
    sharper than asking whether the two Wilson intervals overlap (overlapping 95 % intervals
    can still differ significantly). ``(-1, 1)`` when either side has no trials.
    """
    if trials_a <= 0 or trials_b <= 0:
        return -1.0, 1.0
    low_a, high_a = wilson_interval(successes_a, trials_a, z)
    low_b, high_b = wilson_interval(successes_b, trials_b, z)
    p_a, p_b = successes_a / trials_a, successes_b / trials_b
    delta = p_a - p_b
    lower = delta - math.sqrt((p_a - low_a) ** 2 + (high_b - p_b) ** 2)
    upper = delta + math.sqrt((high_a - p_a) ** 2 + (p_b - low_b) ** 2)
    return max(-1.0, lower), min(1.0, upper)


def trial_case(spec: ControllerSpec, index: int, seed: int = 0, duration: float = 3.0,
               hold_time: float = 1.0, ranges: TrialRanges | None = None,
               base: Config | None = None) -> Case:
    """Trial ``index`` of ``seed``: a closed-loop case with the perturbed plant."""
    from c3bench.bench.closed_loop_suite import Case

    ranges = ranges or TrialRanges()
    scene = (base or load_config()).scene
    rng = np.random.default_rng([seed, index])
    offset = rng.uniform(-ranges.ball_offset, ranges.ball_offset, 2)
    changes = (
        ("cube_side", float(rng.uniform(*ranges.side))),
        ("cube_mass", scene.cube_mass * float(rng.uniform(1 - ranges.mass, 1 + ranges.mass))),
        ("mu_table", scene.mu_table * float(rng.uniform(1 - ranges.friction,
                                                        1 + ranges.friction))),
        ("mu_ball", scene.mu_ball * float(rng.uniform(1 - ranges.friction,
                                                      1 + ranges.friction))),
    )
    model_seed = int(rng.integers(0, 2**31 - 1))
    trial_spec = replace(spec, seed=model_seed) if spec.robust else spec
    name = f"trial-s{seed}-d{duration:g}-h{hold_time:g}-{index:04d}"
    return Case(name, "trials", trial_spec, seed=0, duration=duration,
                scene_changes=changes, ball_offset=(float(offset[0]), float(offset[1])),
                hold_time=hold_time)


def trial_cases(spec: ControllerSpec, trials: int, seed: int = 0, duration: float = 3.0,
                hold_time: float = 1.0, ranges: TrialRanges | None = None) -> list[Case]:
    """The first ``trials`` trials of ``seed`` (:func:`trial_case`)."""
    base = load_config()
    return [trial_case(spec, i, seed, duration, hold_time, ranges, base)
            for i in range(trials)]


def rate_line(label: str, successes: int, trials: int) -> str:
    """``success 14/20 (70%, 95% CI 48-85%)``."""
    low, high = wilson_interval(successes, trials)
    share = 100 * successes / trials if trials else 0.0
    return (f"{label} {successes}/{trials} ({share:.0f}%, 95% CI "
            f"{100 * low:.0f}-{100 * high:.0f}%)")


MEDIANS: tuple[tuple[str, str, float, str], ...] = (
    ("peak_angle", "peak angle", 1.0, "rad"),
    ("hold_time", "hold time", 1.0, "s"),
    ("settling_time", "settling time", 1.0, "s"),
    ("steady_offset", "steady offset", 1.0, "rad"),
    ("impact_speed", "impact speed", 1.0, "m/s"),
    ("contact_time", "time in contact", 1.0, "s"),
    ("free_time", "time out of contact", 1.0, "s"),
    ("max_cube_penetration", "penetration into cube", 1e3, "mm"),
    ("max_table_penetration", "penetration into table", 1e3, "mm"),
    ("clipped_inputs", "clipped inputs", 1.0, "steps"),
    ("plan_lcs_angle_median", "plan vs LCS, angle", 1.0, "rad"),
    ("plan_plant_angle_median", "plan vs plant, angle", 1.0, "rad"),
    ("plan_lcs_error_median", "plan vs LCS, state", 1.0, "norm"),
    ("plan_plant_error_median", "plan vs plant, state", 1.0, "norm"),
    ("median_step_time", "control step", 1e3, "ms"),
)
"""Metrics whose median over the trials is printed: (column, name, scale, unit)."""


def _median(rows: Sequence[dict[str, Any]], column: str) -> float:
    values = np.array([row.get(column, math.nan) for row in rows], dtype=float)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else math.nan


def _label(row: dict[str, Any]) -> str:
    return str(row.get("label") or row.get("failure_label") or "error")


@dataclass(frozen=True)
class TrialSummary:
    """The statistics of a set of trial episodes (one configuration).

    A run that failed to run (``error`` set) counts as a failure: it is in ``n``.

    Attributes
    ----------
    n
        Episodes with a row.
    successes, gentle, passed_balance
        Episodes that succeeded, succeeded gently, passed the balance angle.
    success_interval, gentle_interval
        Wilson 95 % intervals of the two rates (:func:`wilson_interval`).
    errors
        Episodes that produced no run (``error`` set).
    medians
        Median over the episodes of each column of :data:`MEDIANS` (NaN values ignored;
        NaN when none is finite).
    labels
        Count of each label, most common first.
    """

    n: int
    successes: int
    gentle: int
    passed_balance: int
    success_interval: tuple[float, float]
    gentle_interval: tuple[float, float]
    errors: int
    medians: dict[str, float] = field(default_factory=dict)
    labels: tuple[tuple[str, int], ...] = ()

    @property
    def rate(self) -> float:
        """Success rate (NaN without episodes)."""
        return self.successes / self.n if self.n else math.nan


def trial_summary(rows: Sequence[dict[str, Any]]) -> TrialSummary:
    """:class:`TrialSummary` of the rows of one configuration's episodes."""
    done = len(rows)
    success = sum(bool(row.get("success")) for row in rows)
    gentle = sum(bool(row.get("gentle_success")) for row in rows)
    return TrialSummary(
        n=done, successes=success, gentle=gentle,
        passed_balance=sum(bool(row.get("passed_balance")) for row in rows),
        success_interval=wilson_interval(success, done),
        gentle_interval=wilson_interval(gentle, done),
        errors=sum(bool(row.get("error")) for row in rows),
        medians={column: _median(rows, column) for column, *_ in MEDIANS},
        labels=tuple(Counter(_label(row) for row in rows).most_common()))


def summary_lines(rows: Sequence[dict[str, Any]], trials: int) -> list[str]:
    """The printed summary of a trials run (``trials`` episodes asked for; a missing one
    counts in neither numerator nor denominator, a run that failed to run as a failure)."""
    summary = trial_summary(rows)
    done = summary.n
    lines = [rate_line("success", summary.successes, done),
             rate_line("gentle success", summary.gentle, done) + "  (success without passing "
             "the balance angle)",
             f"passed balance  {summary.passed_balance}/{done} (peak angle above "
             "atan(l/2 / l/2) = pi/4)"]
    if done < trials:
        lines.append(f"missing         {trials - done} of {trials} trials (run again)")
    lines.append("medians over the trials:")
    for column, name, scale, unit in MEDIANS:
        value = summary.medians[column]
        shown = "-" if math.isnan(value) else f"{scale * value:.3g}"
        lines.append(f"  {name:<24} {shown} {unit}")
    lines.append("labels: " + ", ".join(f"{label} {count}" for label, count in summary.labels))
    return lines
