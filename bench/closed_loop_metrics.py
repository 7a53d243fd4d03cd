"""Physical metrics of a closed-loop run, and the success rule built on them.

Computed from what :func:`bench.closed_loop.simulate` records: one plant state per control
step (the ball-cube signed distance at each, the commanded and applied inputs, the plan's
predicted next state and the LCS rollout of the plan's first input) and, per control period,
the contact it measured at every plant step (1 ms; :class:`PlantContact`). The contact
metrics and the penetrations are taken at the plant's rate when that record is present, and
from the recorded states alone otherwise (runs recorded before it existed); see
docs/closed_loop.md.

* **peak angle** ``max theta`` and whether it passed the **balance angle**
  ``atan((l/2) / (l/2)) = pi/4`` (the cube's centre of mass over the pivot edge);
* after the ball first **touches** the cube (signed distance <= ``contact_gap``): **time in
  contact** and **time out of contact** (each 1 ms plant state stands for the plant step that
  ended at it; from the recorded states alone, each recorded state but the last stands for
  one control period), and the **impact speed**: the ball's speed relative to the cube (the
  cube's material point at the ball's centre) at the plant state of the touch (from the
  recorded states alone: the ball's speed at the last recorded state before the touch, at the
  touch itself when the run starts in contact); ``contact_step`` is the resolution of these
  (the plant step, or the control period);
* **settling time**: the first time after which ``|theta - theta*|`` stays within the band
  (``success_tolerance``) until the end, and **hold time** ``T_end - settling time`` (0 when
  the run ends outside the band); **steady offset**: the mean of ``theta - theta*`` over the
  last ``hold_time`` seconds;
* **pivot slip**: how far the cube's far bottom corner (the edge it should tip about) moved
  along the table, ``max |x_pivot - x_pivot(0)|`` over the recorded states (NaN when they
  carry no pivot);
* **maximum penetration** of the ball into the cube (``-min`` signed distance) and into the
  table (``-min (z_ball - r - table height)``) over every plant state, 0 when it never
  penetrates;
* **clipped inputs**: control steps whose commanded input exceeded the force limit in some
  coordinate (the simulator applies the clipped one);
* **plan consistency** (median and max over the steps that have a plan): the 2-norm of the
  difference between the plan's predicted next state ``x_1`` and (a) the LCS rollout of the
  plan's first input from the measured state (``lam`` from the step's LCP, Lemke's method),
  (b) the plant's actual next state; also the same for the cube angle alone (rad).

**Success** (:class:`SuccessRules`): the run lasted at least ``min_duration`` (3 s), the
angle stayed within the band for at least ``hold_time`` (1 s) at its end, the pivot slipped
less than ``pivot_slip`` (3 cm: a cube that slid there was pushed along the table, not tipped
about its edge; a run whose pivot was not measured does not succeed), and neither
penetration (at the plant's rate) exceeded ``max_penetration`` (5 mm). **Gentle success**:
success without passing the balance angle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from c3bench.problems.lcs import LCS
from c3bench.solvers.lcp import lemke


@dataclass(frozen=True)
class SuccessRules:
    """Thresholds of the success rule and of the contact metrics.

    Attributes
    ----------
    hold_time
        Seconds the angle must stay within the band at the end of the run.
    min_duration
        Shortest run that can succeed (s).
    max_penetration
        Largest ball penetration into the cube or the table that a success allows (m).
    contact_gap
        Ball-cube signed distance at or below which the ball counts as touching (m).
    pivot_slip
        Slide of the pivot (the cube's far bottom corner) along the table at and beyond which
        the run is no success (m): the cube was pushed, not tipped about its edge. The labels
        of :mod:`bench.closed_loop_labels` call such a run ``cube slid`` with this same
        threshold, and :class:`bench.closed_loop.FailureRules` takes it as its default
        (:func:`bench.closed_loop.summarise` passes a custom one on).
    """

    hold_time: float = 1.0
    min_duration: float = 3.0
    max_penetration: float = 0.005
    contact_gap: float = 0.002
    pivot_slip: float = 0.03

    def __post_init__(self) -> None:
        from c3bench.problems.errors import InputError

        for name in ("hold_time", "min_duration", "max_penetration", "contact_gap",
                     "pivot_slip"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {value!r}")


@dataclass(frozen=True)
class PhysicalMetrics:
    """The physical metrics of one run (module docstring); times in s, angles in rad,
    lengths in m, speeds in m/s. NaN where undefined (no touch, no plan)."""

    peak_angle: float
    balance_angle: float
    passed_balance: bool
    first_touch_time: float
    contact_time: float
    free_time: float
    impact_speed: float
    contact_step: float
    settling_time: float
    hold_time: float
    steady_offset: float
    pivot_slip: float
    max_cube_penetration: float
    max_table_penetration: float
    clipped_inputs: int
    plan_lcs_error_median: float
    plan_lcs_error_max: float
    plan_plant_error_median: float
    plan_plant_error_max: float
    plan_lcs_angle_median: float
    plan_lcs_angle_max: float
    plan_plant_angle_median: float
    plan_plant_angle_max: float
    success: bool
    gentle_success: bool


@dataclass(frozen=True)
class PlantContact:
    """Contact measured at every plant step by :func:`bench.closed_loop.simulate`: one entry
    per control period ``k`` (N-1 of them), over the plant states that end its plant steps
    (the last of them is recorded state ``k + 1``; recorded state 0 belongs to no period).

    Attributes
    ----------
    plant_step
        The plant's time step ``h`` (s); every plant state stands for the step ending at it.
    contact_gap
        Signed distance (m) at or below which :attr:`contact_time` and :attr:`touch_time`
        count the ball as touching (the run's :attr:`SuccessRules.contact_gap`).
    away_gap
        Signed distance (m) above which :attr:`away_time` counts the ball as away (the
        ``contact_gap`` of the failure modes, :class:`bench.closed_loop.FailureRules`).
    min_gap
        Smallest ball-cube signed distance in the period (m; negative: penetration).
    min_height
        Smallest ``z_ball - r - table height`` in the period (m).
    contact_time, away_time
        ``h`` times the number of the period's plant states with signed distance
        ``<= contact_gap``, and ``> away_gap`` (s).
    touch_time
        Time of the period's first plant state with signed distance ``<= contact_gap`` (s;
        NaN when none).
    touch_speed
        At that state, the ball's speed relative to the cube's material point at the ball's
        centre (m/s; NaN when none).
    air_gap
        Height (m) of the cube's lowest point above the table beyond which
        :attr:`cube_air_time` counts the cube as airborne (the ``air_gap`` of the labels,
        :class:`bench.closed_loop_labels.LabelRules`; NaN when not measured).
    cube_clearance, cube_air_time
        The period's largest height of the cube's lowest point above the table (m), and ``h``
        times the number of its plant states with that height ``> air_gap`` (s). Empty for a
        run recorded before they were measured (:attr:`CUBE_COLUMNS`).
    """

    plant_step: float
    contact_gap: float
    away_gap: float
    min_gap: np.ndarray
    min_height: np.ndarray
    contact_time: np.ndarray
    away_time: np.ndarray
    touch_time: np.ndarray
    touch_speed: np.ndarray
    air_gap: float = math.nan
    cube_clearance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cube_air_time: np.ndarray = field(default_factory=lambda: np.zeros(0))

    COLUMNS: ClassVar[tuple[str, ...]] = (
        "min_gap", "min_height", "contact_time", "away_time", "touch_time", "touch_speed")
    """The per-period arrays (stored as ``plant_<name>`` columns of ``steps.csv``)."""
    CUBE_COLUMNS: ClassVar[tuple[str, ...]] = ("cube_clearance", "cube_air_time")
    """The per-period arrays of the cube's height (``plant_<name>`` columns too), both
    present or both empty."""

    def __post_init__(self) -> None:
        lengths = {np.shape(getattr(self, name)) for name in self.COLUMNS}
        if len(lengths) != 1 or len(next(iter(lengths))) != 1:
            raise ValueError(f"PlantContact arrays must be 1-D of one length, got {lengths}")
        cube = {np.shape(getattr(self, name)) for name in self.CUBE_COLUMNS}
        if cube != {(0,)} and cube != lengths:
            raise ValueError(f"PlantContact's cube arrays must be empty or of the others' "
                             f"shape {lengths}, got {cube}")
        if not (math.isfinite(self.plant_step) and self.plant_step > 0):
            raise ValueError(f"plant_step must be > 0, got {self.plant_step!r}")

    def count(self, seconds: float) -> int:
        """``seconds`` as a whole number of plant steps."""
        return round(seconds / self.plant_step)

    @property
    def columns(self) -> tuple[str, ...]:
        """The per-period arrays this record holds (:attr:`COLUMNS`, and
        :attr:`CUBE_COLUMNS` when measured)."""
        return self.COLUMNS + (self.CUBE_COLUMNS if self.cube_air_time.size else ())


@dataclass(frozen=True)
class RunSignals:
    """The per-state signals the metrics need (N recorded states, N-1 control steps).

    Attributes
    ----------
    times, angles
        Time (s) and cube angle (rad) of every recorded state (N).
    ball_gap
        Ball-cube signed distance at every state (N, m; negative: penetration).
    ball_height
        Ball bottom above the table, ``z_ball - r - table height`` (N, m).
    ball_speed
        Ball speed (N, m/s).
    commanded
        The controller's commanded inputs before the simulator's clip (N-1 x nu).
    force_limit
        The simulator's clip (N).
    cube_side
        The plant cube's side (m).
    plan_next, lcs_next
        Per step (N-1 x nx): the plan's predicted next state and the LCS rollout of its first
        input; rows of NaN where the step had no plan.
    states
        The recorded states (N x nx).
    angle_index
        Index of the cube angle in the state.
    ball_above_top, pivot_x, cube_clearance
        Per state (N, or empty when not measured): the ball centre over the cube's top face
        (in the cube frame: above the top face's plane and within its extent), the x of the
        cube's far bottom corner (m; the pivot slip of the success rule, which a run without
        it cannot pass) and the height of the cube's lowest point above the table (m); for
        the labels of :mod:`bench.closed_loop_labels`.
    plant
        The contact measured at every plant step, per control period (N-1; ``None`` for a
        run recorded without it: the contact metrics then use the recorded states alone).
    """

    times: np.ndarray
    angles: np.ndarray
    ball_gap: np.ndarray
    ball_height: np.ndarray
    ball_speed: np.ndarray
    commanded: np.ndarray
    force_limit: float
    cube_side: float
    plan_next: np.ndarray
    lcs_next: np.ndarray
    states: np.ndarray
    angle_index: int = 2
    ball_above_top: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    pivot_x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cube_clearance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plant: PlantContact | None = None


def balance_angle(side_x: float, side_z: float | None = None) -> float:
    """``atan((side_x / 2) / (side_z / 2))``: the tilt that puts the centre of mass over the
    pivot edge (pi/4 for a cube)."""
    height = side_x if side_z is None else side_z
    return math.atan2(side_x / 2, height / 2)


def lcs_rollout(lcs: LCS, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``A x + B u + D lam + d`` with ``lam`` solving ``0 <= lam perp F lam + E x + H u + c
    >= 0`` (Lemke's method; NaN when it finds no solution)."""
    solution = lemke(lcs.F, lcs.lcp_offset(x, u))
    if solution.z is None or not solution.found:
        return np.full(lcs.nx, np.nan)
    return lcs.next_state(x, u, solution.z)


def plan_prediction(samples: Sequence[LCS], delta: np.ndarray, weights: np.ndarray | None,
                    x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(plan x_1, LCS rollout of the plan's u_0, u_0)``, weighted over the samples.

    ``delta`` is (S, T, step) with ``x, lam, u`` first in each step (C3 and C3+ layouts);
    sample ``j``'s plan is rolled out through sample ``j``'s LCS from the measured ``x``.
    """
    delta = np.asarray(delta, dtype=float)
    count = min(len(samples), delta.shape[0])
    p = np.full(count, 1.0 / count) if weights is None else \
        np.asarray(weights, dtype=float)[:count] / np.sum(np.asarray(weights)[:count])
    nx, nlam, nu = samples[0].nx, samples[0].nlam, samples[0].nu
    second = 1 if delta.shape[1] > 1 else 0
    plans = delta[:count, second, :nx]
    inputs = delta[:count, 0, nx + nlam: nx + nlam + nu]
    rollouts = np.array([lcs_rollout(samples[j], x, inputs[j]) for j in range(count)])
    return p @ plans, p @ rollouts, p @ inputs


def _nan_stats(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if not finite.size:
        return math.nan, math.nan
    return float(np.median(finite)), float(np.max(finite))


def _contact(signals: RunSignals, rules: SuccessRules
             ) -> tuple[float, float, float, float, float]:
    """``(first touch time, time in contact, time out of contact, impact speed, resolution)``,
    at the plant's rate when :attr:`RunSignals.plant` is there, else from the recorded
    states."""
    plant = signals.plant
    if plant is None:
        return _sampled_contact(signals, rules)
    if not math.isclose(plant.contact_gap, rules.contact_gap, rel_tol=1e-12, abs_tol=1e-15):
        raise ValueError(f"the plant-rate contact was measured at contact_gap "
                         f"{plant.contact_gap!r}, the rules ask for {rules.contact_gap!r}")
    if signals.ball_gap[0] <= rules.contact_gap:  # the run starts in contact
        first, period, speed, own = float(signals.times[0]), 0, float(signals.ball_speed[0]), 0
    else:
        hits = np.flatnonzero(np.isfinite(plant.touch_time))
        if not hits.size:
            return math.nan, 0.0, 0.0, math.nan, plant.plant_step
        period = int(hits[0])
        first, speed, own = float(plant.touch_time[period]), \
            float(plant.touch_speed[period]), 1  # the touching state itself is not "after"
    touching = plant.count(float(np.sum(plant.contact_time[period:]))) - own
    after = plant.count(float(signals.times[-1]) - first)
    h = plant.plant_step
    return first, touching * h, max(after - touching, 0) * h, speed, h


def _sampled_contact(signals: RunSignals, rules: SuccessRules
                     ) -> tuple[float, float, float, float, float]:
    """:func:`_contact` from the recorded states alone (each but the last stands for one
    control period; impact speed at the last state before the touch)."""
    touching = signals.ball_gap <= rules.contact_gap
    hits = np.flatnonzero(touching)
    periods = np.diff(signals.times)
    resolution = float(np.median(periods)) if periods.size else math.nan
    if not hits.size:
        return math.nan, 0.0, 0.0, math.nan, resolution
    first = int(hits[0])
    inside = touching[first:-1]
    contact = float(np.sum(periods[first:][inside]))
    free = float(np.sum(periods[first:][~inside]))
    speed = float(signals.ball_speed[max(first - 1, 0)])
    return float(signals.times[first]), contact, free, speed, resolution


def _penetrations(signals: RunSignals) -> tuple[float, float]:
    """Deepest ball penetration into the cube and into the table (m, >= 0), over every plant
    state when :attr:`RunSignals.plant` is there."""
    gaps, heights = [signals.ball_gap], [signals.ball_height]
    if signals.plant is not None and signals.plant.min_gap.size:
        gaps.append(signals.plant.min_gap)
        heights.append(signals.plant.min_height)
    return (max(0.0, -float(np.min(np.concatenate(gaps)))),
            max(0.0, -float(np.min(np.concatenate(heights)))))


def pivot_slip(pivot_x: np.ndarray) -> float:
    """``max |x_pivot - x_pivot(0)|`` over the recorded states' pivot x (m; NaN when there is
    none: :attr:`RunSignals.pivot_x` not measured). The failure modes of
    :func:`bench.closed_loop.label_failure_mode` take it too."""
    return float(np.max(np.abs(pivot_x - pivot_x[0]))) if pivot_x.size else math.nan


def _settling(signals: RunSignals, target: float, band: float) -> tuple[float, float]:
    """``(settling time, hold time)``: from the first state after which the angle stays within
    the band to the end (NaN, 0 when the run ends outside it)."""
    inside = np.abs(signals.angles - target) <= band
    if not inside[-1]:
        return math.nan, 0.0
    outside = np.flatnonzero(~inside)
    start = int(outside[-1]) + 1 if outside.size else 0
    settle = float(signals.times[start])
    return settle, float(signals.times[-1] - settle)


def _consistency(signals: RunSignals) -> dict[str, float]:
    """Median and max of the plan's next-state error against the LCS and the plant, as a
    state 2-norm and in the cube angle."""
    actual = signals.states[1:]
    plan, lcs = signals.plan_next, signals.lcs_next
    k = signals.angle_index
    out: dict[str, float] = {}
    for name, error in (("plan_lcs_error", np.linalg.norm(plan - lcs, axis=1)),
                        ("plan_plant_error", np.linalg.norm(plan - actual, axis=1)),
                        ("plan_lcs_angle", np.abs(plan[:, k] - lcs[:, k])),
                        ("plan_plant_angle", np.abs(plan[:, k] - actual[:, k]))):
        out[f"{name}_median"], out[f"{name}_max"] = _nan_stats(error)
    return out


def physical_metrics(signals: RunSignals, target: float, band: float,
                     rules: SuccessRules | None = None) -> PhysicalMetrics:
    """The metrics of one run and its success (module docstring).

    Parameters
    ----------
    signals
        What the run recorded.
    target, band
        Target angle ``theta*`` and the half-width of the success band (rad).
    rules
        Success thresholds (default :class:`SuccessRules`).
    """
    rules = rules or SuccessRules()
    peak = float(np.max(signals.angles))
    balance = balance_angle(signals.cube_side)
    touch, contact, free, speed, resolution = _contact(signals, rules)
    settle, hold = _settling(signals, target, band)
    window = signals.times >= signals.times[-1] - rules.hold_time - 1e-9
    offset = float(np.mean(signals.angles[window] - target))
    cube_pen, table_pen = _penetrations(signals)
    clipped = int(np.sum(np.any(np.abs(signals.commanded) > signals.force_limit + 1e-9,
                                axis=1))) if signals.commanded.size else 0
    duration = float(signals.times[-1] - signals.times[0])
    slip = pivot_slip(signals.pivot_x)
    success = (duration >= rules.min_duration - 1e-9 and hold >= rules.hold_time - 1e-9
               and slip < rules.pivot_slip  # False when not measured (NaN)
               and max(cube_pen, table_pen) <= rules.max_penetration)
    passed = peak > balance
    return PhysicalMetrics(
        peak_angle=peak, balance_angle=balance, passed_balance=passed, first_touch_time=touch,
        contact_time=contact, free_time=free, impact_speed=speed, contact_step=resolution,
        settling_time=settle,
        hold_time=hold, steady_offset=offset, pivot_slip=slip, max_cube_penetration=cube_pen,
        max_table_penetration=table_pen, clipped_inputs=clipped, **_consistency(signals),
        success=success, gentle_success=success and not passed)
